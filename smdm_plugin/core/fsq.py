"""Finite scalar quantisation (Mentzer et al. 2023) and an ``nn.MultiheadAttention`` drop-in
whose attention keys are FSQ-quantised.

FSQ bounds each of ``d = len(levels)`` channels to ``L_i`` integer levels, rounds with a
straight-through estimator and rescales to ``[-1, 1]``. :class:`FSQMultiheadAttention` keeps
``nn.MultiheadAttention``'s parameter names (``in_proj_weight``, ``in_proj_bias``,
``out_proj.weight``, ``out_proj.bias``) so dense checkpoints load into it, and adds ``key_down``
(``head_dim -> d``) and ``key_up`` (``d -> head_dim``), shared by all heads.
"""
from __future__ import annotations

import math
from typing import Any, List, Optional, Sequence, Tuple

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from .attention import (accelerator_path, aligned_key_bias, attend, attend_with_weights, compute_dtype, float_mask,
                        heads, layout_copies, project_qkv)
from .checks import compiling
from .fsq_bank import KeyMapBank, bank_key_maps, key_map_tensors, remove_banks, shared_bank
from .kernels.fsq_code import fsq_code
from .products import ProductStore, held_products, store_of

__all__ = ["FSQ", "FSQMultiheadAttention", "quantize_attention_keys"]


class _RoundSTE(torch.autograd.Function):
    """``torch.round`` whose gradient is the identity (straight-through): one op forward, none
    backward (``b + (round(b) - b).detach()`` costs three)."""

    @staticmethod
    def forward(ctx, b: Tensor) -> Tensor:
        return torch.round(b)

    @staticmethod
    def backward(ctx, g: Tensor) -> Tensor:
        return g


def cast_once(module: nn.Module, name: str, bufs: Tuple[Tensor, ...], dtype: torch.dtype) -> Tuple[Tensor, ...]:
    """``bufs`` in ``dtype``: cast once per dtype (outside tracing) and kept in ``module``'s store
    ``name`` (:class:`~smdm_plugin.core.products.ProductStore`: a move or an in-place update makes new
    copies), not at every use (under autocast, each use of a float32 buffer in a bf16 op would be a
    cast kernel)."""
    if bufs[0].dtype == dtype:
        return bufs
    if compiling():
        return tuple(b.to(dtype) for b in bufs)
    return store_of(module, name).get(dtype, bufs, lambda: [b.to(dtype) for b in bufs])


class FSQ(nn.Module):
    """Finite scalar quantiser. ``[..., d] -> [..., d]`` with ``d = len(levels)``.

    Channel ``i`` is bounded to ``(L_i - 1)/2 · tanh`` (shifted by half a level for even
    ``L_i`` so that it covers ``L_i`` integers ``-floor(L_i/2) .. ceil(L_i/2) - 1``), rounded
    (straight-through: the gradient of the rounding is the identity) and divided by
    ``floor(L_i/2)``. Output values lie on the grid ``{k / floor(L_i/2)}`` inside ``[-1, 1]``.
    """

    def __init__(self, levels: Sequence[int], eps: float = 1e-3) -> None:
        super().__init__()
        levels = [int(v) for v in levels]
        if not levels or any(v < 2 for v in levels):
            raise ValueError(f"FSQ: levels must be a non-empty sequence of ints >= 2, got {levels}")
        self.levels_list = tuple(levels)
        lv = torch.tensor(levels, dtype=torch.float64)
        half_l = (lv - 1) * (1 - eps) / 2                        # tanh amplitude
        offset = torch.where(lv % 2 == 0, 0.5, 0.0)              # even L: asymmetric range
        # shift as in the paper: tan(offset / half_l) (~ atanh for L >= 4, so bound(0) ~ 0;
        # finite for L = 2, where atanh(offset / half_l) does not exist)
        shift = torch.tan(offset / half_l)
        basis = torch.cumprod(torch.tensor([1] + levels[:-1], dtype=torch.long), 0)
        # non-persistent: a dense checkpoint carries no FSQ buffers
        self.register_buffer("_half_l", half_l.float(), persistent=False)
        self.register_buffer("_offset", offset.float(), persistent=False)
        self.register_buffer("_neg_offset", -offset.float(), persistent=False)
        self.register_buffer("_shift", shift.float(), persistent=False)
        self.register_buffer("_half_width", (lv // 2).float(), persistent=False)
        self.register_buffer("_basis", basis, persistent=False)

    def constants(self, dtype: torch.dtype) -> Tuple[Tensor, Tensor, Tensor, Tensor]:
        """``(neg_offset, half_l, shift, half_width)`` ``[d]`` in ``dtype``: cast once per dtype and
        device (outside tracing), not at every use (under autocast, each use of a float32 buffer
        in a bf16 op would be a cast kernel); keyed on the buffers' storage and version."""
        return cast_once(self, "_constant_casts", (self._neg_offset, self._half_l, self._shift, self._half_width),
                         dtype)

    @property
    def dim(self) -> int:
        return len(self.levels_list)

    @property
    def codebook_size(self) -> int:
        return int(math.prod(self.levels_list))

    def bound(self, z: Tensor, shifted: bool = False) -> Tensor:
        """``[..., d]``: each channel squashed into ``(-floor(L/2) - 0.5, ceil(L/2) - 0.5)``
        (``tanh(z + shift) * half_l - offset``, as one fused multiply-add; ``shifted``: ``z``
        already holds ``+ shift``)."""
        neg_offset, half_l, shift, _ = self.constants(z.dtype)
        t = torch.tanh(z if shifted else z + shift)
        return torch.addcmul(neg_offset, t, half_l)

    @staticmethod
    def round(b: Tensor) -> Tensor:
        """Integer levels of bounded ``b``; straight-through under autograd (identity gradient)."""
        return _RoundSTE.apply(b) if torch.is_grad_enabled() and b.requires_grad else torch.round(b)

    def forward(self, z: Tensor) -> Tensor:
        if z.shape[-1] != self.dim:
            raise ValueError(f"FSQ: input must be [..., {self.dim}], got {tuple(z.shape)}")
        return self.round(self.bound(z)) / self.constants(z.dtype)[3]

    def codes_to_indices(self, codes: Tensor) -> Tensor:
        """``[..., d]`` grid codes (as returned by ``forward``) -> ``[...]`` long in
        ``[0, codebook_size)``."""
        hw = self._half_width.to(codes.dtype)
        digits = torch.round(codes * hw + hw).long()
        return (digits * self._basis).sum(-1)

    def indices_to_codes(self, indices: Tensor) -> Tensor:
        """``[...]`` long -> ``[..., d]`` grid codes (float32)."""
        levels = torch.tensor(self.levels_list, device=indices.device)
        digits = (indices.long().unsqueeze(-1) // self._basis) % levels
        hw = self._half_width
        return (digits.float() - hw) / hw

    def extra_repr(self) -> str:
        return f"levels={list(self.levels_list)}, codebook_size={self.codebook_size}"


def _disable_transformer_fast_path(module: nn.Module, args: Any) -> None:
    """No-op forward pre-hook. Its presence makes ``nn.TransformerEncoderLayer`` skip its fused
    fast path (which would call the dense attention kernel directly and bypass FSQ)."""
    return None


class FSQMultiheadAttention(nn.Module):
    """``nn.MultiheadAttention`` drop-in whose keys are FSQ-quantised per head.

    ``k = key_up(FSQ(key_down(k_head)))`` for each head's ``k_head [.., head_dim]``, then scaled
    dot-product attention. Shapes as ``nn.MultiheadAttention``: ``query [L, B, E]`` (``[B, L, E]``
    with ``batch_first``; ``[L, E]`` unbatched), ``key``/``value [S, B, E]``,
    ``key_padding_mask [B, S]`` (bool True = ignore, or additive float), ``attn_mask [L, S]`` or
    ``[B·H, L, S]`` (bool True = not allowed, or additive float). Returns ``(out, weights)`` with
    ``weights [B, L, S]`` (``[B, H, L, S]`` if not ``average_attn_weights``) or ``None``.

    Set ``quantize = False`` to bypass the key bottleneck (then it equals dense attention).
    Unsupported ``nn.MultiheadAttention`` options: ``kdim``/``vdim != embed_dim``,
    ``add_bias_kv``, ``add_zero_attn``.
    """

    def __init__(self, embed_dim: int, num_heads: int, dropout: float = 0.0, bias: bool = True,
                 add_bias_kv: bool = False, add_zero_attn: bool = False,
                 kdim: Optional[int] = None, vdim: Optional[int] = None,
                 batch_first: bool = False, levels: Sequence[int] = (8, 8, 8, 5, 5, 5),
                 device: Optional[torch.device] = None, dtype: Optional[torch.dtype] = None
                 ) -> None:
        super().__init__()
        if embed_dim <= 0 or num_heads <= 0 or embed_dim % num_heads:
            raise ValueError(f"FSQMultiheadAttention: embed_dim={embed_dim} must be a positive "
                             f"multiple of num_heads={num_heads}")
        if add_bias_kv or add_zero_attn or kdim not in (None, embed_dim) \
                or vdim not in (None, embed_dim):
            raise ValueError("FSQMultiheadAttention: add_bias_kv, add_zero_attn and "
                             "kdim/vdim != embed_dim are not supported")
        # drawn on the CPU, then moved: the same seed gives the same weights on every device, and
        # the device's own generator (upstream's noise on CUDA) is not advanced
        target = torch.device(device) if device is not None else torch.empty(0).device
        fk = {"device": torch.device("cpu"), "dtype": dtype}
        self.embed_dim, self.num_heads = int(embed_dim), int(num_heads)
        self.head_dim = self.embed_dim // self.num_heads
        self.kdim = self.vdim = self.embed_dim
        self._qkv_same_embed_dim = True
        self.dropout, self.batch_first = float(dropout), bool(batch_first)
        self.bias_k = self.bias_v = None
        self.add_zero_attn = False
        self.in_proj_weight = nn.Parameter(torch.empty(3 * self.embed_dim, self.embed_dim, **fk))
        self.in_proj_bias = nn.Parameter(torch.empty(3 * self.embed_dim, **fk)) if bias else None
        self.out_proj = nn.Linear(self.embed_dim, self.embed_dim, bias=bias, **fk)
        self.fsq = FSQ(levels)
        self.key_down = nn.Linear(self.head_dim, self.fsq.dim, **fk)
        self.key_up = nn.Linear(self.fsq.dim, self.head_dim, **fk)
        self.quantize = True
        self._call_proj: Optional[Tuple[Tensor, Tensor]] = None    # set by fold_keys for one call
        # the code channels of the folded path (:meth:`_forward_folded`): the ``d`` FSQ channels and
        # zeros up to a multiple of 8 (the head sizes GPU attention kernels take); per channel the
        # bound's ``neg_offset`` and ``half_l`` (0 on the padding: its codes are 0), tiled over the heads
        pad = self.code_dim - self.fsq.dim
        self.register_buffer("_code_neg_offset", F.pad(self.fsq._neg_offset, (0, pad)).repeat(self.num_heads),
                             persistent=False)
        self.register_buffer("_code_half_l", F.pad(self.fsq._half_l, (0, pad)).repeat(self.num_heads),
                             persistent=False)
        # key_up.bias adds q·bias to every key's logit of a query: softmax does not see it (its
        # gradient is exactly 0), and the folded path does not read it; frozen, so that optimizers
        # and DDP (find_unused_parameters=False) see no trainable parameter without a gradient
        self.key_up.bias.requires_grad_(False)
        self._reset_parameters()
        if target.type != "cpu":
            self.to(target)
        self.register_forward_pre_hook(_disable_transformer_fast_path)

    def _reset_parameters(self) -> None:
        nn.init.xavier_uniform_(self.in_proj_weight)
        if self.in_proj_bias is not None:
            nn.init.zeros_(self.in_proj_bias)
            nn.init.zeros_(self.out_proj.bias)

    @classmethod
    def from_mha(cls, mha: nn.MultiheadAttention, levels: Sequence[int]
                 ) -> "FSQMultiheadAttention":
        """A copy of ``mha``'s projections (and train/eval mode) with FSQ keys."""
        if not mha._qkv_same_embed_dim or mha.bias_k is not None or mha.add_zero_attn:
            raise ValueError("FSQMultiheadAttention.from_mha: mha must have kdim = vdim = "
                             "embed_dim, no add_bias_kv and no add_zero_attn")
        w = mha.in_proj_weight
        new = cls(mha.embed_dim, mha.num_heads, dropout=mha.dropout,
                  bias=mha.in_proj_bias is not None, batch_first=mha.batch_first,
                  levels=levels, device=w.device, dtype=w.dtype)
        missing, unexpected = new.load_state_dict(mha.state_dict(), strict=False)
        assert not unexpected and all(k.startswith(("key_down.", "key_up.")) for k in missing)
        return new.train(mha.training)

    def to_mha(self) -> nn.MultiheadAttention:
        """The dense ``nn.MultiheadAttention`` with this layer's current q/k/v/out weights (and
        train/eval mode); the key codebook projections (``key_down``/``key_up``) are dropped."""
        w = self.in_proj_weight
        mha = nn.MultiheadAttention(self.embed_dim, self.num_heads, dropout=self.dropout,
                                    bias=self.in_proj_bias is not None, batch_first=self.batch_first,
                                    device=w.device, dtype=w.dtype)
        own = self.state_dict()
        mha.load_state_dict({k: own[k] for k in mha.state_dict()})
        return mha.train(self.training)

    def _heads(self, x: Tensor, batch_first: bool) -> Tensor:
        """``[B, T, E]`` (``batch_first``) or ``[T, B, E]`` -> ``[B, H, T, head_dim]``: :meth:`_heads_of`."""
        return self._heads_of(x, batch_first, self.head_dim)

    def quantize_keys(self, k: Tensor) -> Tensor:
        """``[..., S, head_dim] -> [..., S, head_dim]`` through the FSQ bottleneck. ``key_down``
        runs as one batched matmul over dim ``-2`` (the heads, for the layout ``[.., H, head_dim]``
        of the in-projection's keys), which reads strided keys in place (no copy); ``key_up`` as
        one fused multiply-add on the rows. The result has ``k``'s shape (strides may differ)."""
        S, hd = k.shape[-2:]
        kb = k.movedim(-2, 0).reshape(S, -1, hd)                        # [S, M, hd]: a view for the keys
        down_bias, down_weight_t, up_weight, up_bias = self._folded(compute_dtype(k))
        # W^T as the transpose of W expanded (not W^T expanded): the same values, and the weight's
        # gradient (the sum over the heads) comes out in W's own layout (no copy into it)
        down_weight = down_weight_t.t().expand(S, self.fsq.dim, hd).transpose(1, 2)
        z = torch.baddbmm(down_bias, kb, down_weight)
        r = self.fsq.round(self.fsq.bound(z, shifted=True))              # [S, M, d] integer levels
        out = F.linear(r.view(-1, self.fsq.dim), up_weight, up_bias)   # [S*M, hd]
        return out.view(S, *k.shape[:-2], hd).movedim(0, -2)

    def _folded(self, dtype: torch.dtype) -> Tuple[Tensor, Tensor, Tensor, Tensor]:
        """FSQ's constant affine steps folded into the two projections: ``(key_down.bias + shift
        [d], key_down.weight.t() [head_dim, d], key_up.weight / floor(L/2) [head_dim, d],
        key_up.bias [head_dim])``. Without autograd (sampling) and outside tracing, cached in the
        compute ``dtype`` (autocast's, else the keys'): keyed on the parameters' storage and
        version, as the Lipschitz layers; so a sampling call under autocast casts none of them (the
        values autocast would make). With autograd: the parameters' dtype (autocast casts them)."""
        if not torch.is_grad_enabled() and not compiling():
            inputs = (*key_map_tensors(self), self.fsq._shift, self.fsq._half_width)
            return store_of(self, "_key_map_store").get(dtype, inputs,
                                                        lambda: [t.to(dtype) for t in self._key_map_values()])
        return self._key_map_values()

    def _key_map_values(self) -> Tuple[Tensor, Tensor, Tensor, Tensor]:
        down, up, fsq = self.key_down, self.key_up, self.fsq
        _, _, shift, half_width = fsq.constants(down.bias.dtype)
        return (down.bias + shift, down.weight.t(), up.weight / half_width, up.bias)

    @property
    def code_dim(self) -> int:
        """``P``: channels of a head's query and key on the folded path: the ``d`` FSQ channels,
        zeros up to a multiple of 8."""
        return -(-self.fsq.dim // 8) * 8

    def code_constants(self, dtype: torch.dtype) -> Tuple[Tensor, Tensor]:
        """``(neg_offset, half_l)`` ``[H·P]`` of the folded path's bound (every head's ``P``
        channels) in ``dtype`` (cast once per dtype outside tracing, as :meth:`FSQ.constants`)."""
        return cast_once(self, "_code_casts", (self._code_neg_offset, self._code_half_l), dtype)

    def _projection(self, dtype: torch.dtype) -> Tuple[Tensor, Tensor]:
        """This layer's folded in-projection (:func:`folded_projections`) for a call computing in
        ``dtype``: the one :class:`fold_keys` made for all layers, else, without autograd, kept in
        ``dtype`` in its :class:`~smdm_plugin.core.products.ProductStore` (keyed on the parameters'
        storage and version; an armed trace reads it as it is), else made for this layer alone."""
        call = self.__dict__.get("_call_proj")
        if call is not None:
            return call
        if not torch.is_grad_enabled():
            if not compiling():
                return self.refresh_products(dtype)
            held = held_products(self, dtype)
            if held is not None:
                return held
        return folded_projections([self], None)[0]

    def products(self) -> ProductStore:
        """What this layer's calls without autograd make from its parameters alone."""
        return store_of(self)

    def refresh_products(self, dtype: Optional[torch.dtype] = None) -> Tuple[Tensor, Tensor]:
        """The folded in-projection ``(weight, bias)`` in ``dtype`` (default: the dtype a call computes
        in now, :func:`~smdm_plugin.core.attention.compute_dtype`), remade in place when a parameter
        changed (with the other dtypes held: :meth:`ProductStore.refresh`)."""
        dtype = compute_dtype(self.in_proj_weight) if dtype is None else dtype
        return store_of(self).refresh(dtype, self._fold_inputs(), lambda d: folded_projections([self], d)[0])

    def product_inputs(self) -> Tuple[Tensor, ...]:
        """Every tensor the folded in-projection is made of (:mod:`~smdm_plugin.core.products`)."""
        return self._fold_inputs()

    def _fold_inputs(self) -> Tuple[Tensor, ...]:
        b = self.in_proj_bias
        return (self.in_proj_weight, *key_map_tensors(self)[:3], self.fsq._shift,
                self.fsq._half_width) + (() if b is None else (b,))

    def _forward_folded(self, x: Tensor, bf: bool, mask: Optional[Tensor], need_weights: bool
                        ) -> Tuple[Tensor, Optional[Tensor]]:
        """Self-attention on the folded path: one in-projection gives each head's query code
        ``q·key_up.weight / floor(L/2)``, key pre-code ``key_down(k) + shift`` (``P`` channels each,
        zero-padded) and the values; the keys' codes are ``round(bound(.))``; attention on
        ``P``-channel queries and keys with the scale of ``head_dim``. The same attention as
        ``q·key_up(FSQ(key_down(k)))`` in real arithmetic (``q·key_up.bias`` is the same for every
        key of a query: softmax drops it), without key_down / key_up on the activations.
        ``x [T, B, E]`` (``[B, T, E]`` with ``bf``)."""
        E, H, hd, P = self.embed_dim, self.num_heads, self.head_dim, self.code_dim
        weight, bias = self._projection(compute_dtype(x))
        qc, z, v = F.linear(x, weight, bias).split([H * P, H * P, E], dim=-1)
        neg_offset, half_l = self.code_constants(torch.float32)
        r = fsq_code(z, neg_offset, half_l)                        # [.., H·P] codes, one op each way
        qc, r, v = self._heads_of(qc, bf, P), self._heads_of(r, bf, P), self._heads(v, bf)
        scale = 1.0 / math.sqrt(hd)
        if need_weights:
            return attend_with_weights(self, qc, r, v, mask, scale)
        return attend(self, qc, r, v, mask, scale), None

    def _heads_of(self, x: Tensor, batch_first: bool, size: int) -> Tensor:
        """``[B, T, H·size]`` (``batch_first``) or ``[T, B, H·size]`` -> ``[B, H, T, size]``: a view
        (of a contiguous ``[B, T, H·size]`` copy when :func:`~smdm_plugin.core.attention.use_layout_copies`
        is on)."""
        copy = layout_copies()
        if not batch_first:
            return heads(x, self.num_heads, copy)
        if copy:
            x = x.contiguous()
        return x.unflatten(-1, (self.num_heads, size)).transpose(1, 2)

    def forward(self, query: Tensor, key: Tensor, value: Tensor,
                key_padding_mask: Optional[Tensor] = None, need_weights: bool = True,
                attn_mask: Optional[Tensor] = None, average_attn_weights: bool = True,
                is_causal: bool = False) -> Tuple[Tensor, Optional[Tensor]]:
        if query.is_nested or key.is_nested or value.is_nested:
            return self._forward_nested(query, key, value, need_weights, attn_mask,
                                        average_attn_weights, is_causal)
        unbatched = query.dim() == 2
        if unbatched:
            query, key, value = query.unsqueeze(1), key.unsqueeze(1), value.unsqueeze(1)
            if key_padding_mask is not None:
                key_padding_mask = key_padding_mask.unsqueeze(0)
        bf = not unbatched and self.batch_first                    # else [T, B, E]
        E, H, hd = self.embed_dim, self.num_heads, self.head_dim
        B = query.shape[0] if bf else query.shape[1]
        L, S = query.shape[1 if bf else 0], key.shape[1 if bf else 0]
        dt = compute_dtype(query) if query.is_floating_point() else query.dtype
        mask = self._mask(attn_mask, key_padding_mask, is_causal, B, L, S, dt, query.device)
        if self.quantize and query is key and key is value:
            out, weights = self._forward_folded(query, bf, mask, need_weights)
        else:
            q, k, v = project_qkv(self, query, key, value)         # in the input's own layout
            q, v = self._heads(q, bf), self._heads(v, bf)           # [B, H, T, hd]
            if self.quantize:                                       # [T, B, H, hd] or [B, T, H, hd]
                k = self._heads(self.quantize_keys(k.unflatten(-1, (H, hd))).flatten(-2), bf)
            else:
                k = self._heads(k, bf)
            if need_weights:
                out, weights = attend_with_weights(self, q, k, v, mask)   # weights [B, H, L, S]
            else:
                out, weights = attend(self, q, k, v, mask), None
        if weights is not None and average_attn_weights:
            weights = weights.mean(dim=1)
        out = out.permute(0, 2, 1, 3) if bf else out.permute(2, 0, 1, 3)   # [B, L, H, hd] / [L, B, H, hd]
        out = self.out_proj(out.reshape(-1, E)).view(*out.shape[:2], E)
        if unbatched:
            return out.squeeze(1), None if weights is None else weights.squeeze(0)
        return out, weights

    def _mask(self, attn_mask: Optional[Tensor], key_padding_mask: Optional[Tensor], is_causal: bool,
              B: int, L: int, S: int, dt: torch.dtype, device: torch.device) -> Optional[Tensor]:
        """The combined additive mask in ``dt``, broadcastable to ``[B, H, L, S]``, or None."""
        H = self.num_heads
        mask = float_mask(attn_mask, dt)
        if mask is None and is_causal:
            mask = torch.full((L, S), float("-inf"), dtype=dt, device=device).triu(1)
        if mask is not None:
            if mask.shape[-2:] != (L, S) or mask.dim() not in (2, 3):
                raise ValueError(f"FSQMultiheadAttention: attn_mask must be [L={L}, S={S}] or "
                                 f"[B*H={B * H}, L, S], got {tuple(mask.shape)}")
            mask = mask.reshape(B, H, L, S) if mask.dim() == 3 else mask.reshape(1, 1, L, S)
        kpm = float_mask(key_padding_mask, dt)
        if kpm is not None:
            if kpm.shape != (B, S):
                raise ValueError(f"FSQMultiheadAttention: key_padding_mask must be [B={B}, "
                                 f"S={S}], got {tuple(kpm.shape)}")
            kpm = kpm.view(B, 1, 1, S)
            mask = kpm if mask is None else mask + kpm
        if mask is not None and accelerator_path(mask):
            mask = aligned_key_bias(mask)                           # rows every SDPA kernel reads
        return mask

    def _forward_nested(self, query: Tensor, key: Tensor, value: Tensor, need_weights: bool,
                        attn_mask: Optional[Tensor], average_attn_weights: bool, is_causal: bool
                        ) -> Tuple[Tensor, Optional[Tensor]]:
        """Nested (batch-first) input, as ``nn.TransformerEncoder`` produces in eval with a
        padding mask: pad, mask the padded keys, run, re-nest the output."""
        if not self.batch_first or not (query.is_nested and key.is_nested and value.is_nested):
            raise ValueError("FSQMultiheadAttention: nested input needs batch_first=True and "
                             "nested query, key and value")

        def lengths(t: Tensor) -> list:
            return [int(u.shape[0]) for u in t.unbind()]

        q = query.to_padded_tensor(0.0)
        k = q if key is query else key.to_padded_tensor(0.0)
        v = q if value is query else value.to_padded_tensor(0.0)
        lk = torch.tensor(lengths(key), device=k.device)
        kpm = torch.arange(k.shape[1], device=k.device)[None, :] >= lk[:, None]   # [B, S]
        out, weights = self.forward(q, k, v, key_padding_mask=kpm, need_weights=need_weights,
                                    attn_mask=attn_mask, average_attn_weights=average_attn_weights,
                                    is_causal=is_causal)
        out = torch.nested.as_nested_tensor(
            [o[:n] for o, n in zip(out.unbind(0), lengths(query))], layout=query.layout)
        return out, weights

    def extra_repr(self) -> str:
        return (f"embed_dim={self.embed_dim}, num_heads={self.num_heads}, "
                f"dropout={self.dropout}, batch_first={self.batch_first}, quantize={self.quantize}")


def _stack(ts: Sequence[Tensor]) -> Tensor:
    """``[G, ...]``: ``torch.stack``, a view for one tensor."""
    return ts[0].unsqueeze(0) if len(ts) == 1 else torch.stack(list(ts))


def folded_projections(attns: Sequence["FSQMultiheadAttention"], dtype: Optional[torch.dtype] = None,
                       bank: Optional[KeyMapBank] = None) -> List[Tuple[Tensor, Tensor]]:
    """The in-projections of the folded path (:meth:`FSQMultiheadAttention._forward_folded`) of
    every layer in ``attns`` (the same sizes, levels and dtype), made at once for all layers:
    ``(weight [2·H·P + E, E], bias [2·H·P + E])`` per layer, rows ``[query codes (H·P), key
    pre-codes (H·P), values (E)]``. Per head ``h``, with ``U = [key_up.weight / floor(L/2) | 0]
    [hd, P]`` and ``D = [key_down.weight; 0] [P, hd]``: query codes ``U^T (W_q,h x + b_q,h)``, key
    pre-codes ``D (W_k,h x + b_k,h) + [key_down.bias + shift; 0]``. Differentiable in every
    parameter it reads; computed in the parameters' dtype, then cast to ``dtype`` when given. The
    layers' key maps are read as they are when a :class:`~smdm_plugin.core.fsq_bank.KeyMapBank` holds
    exactly them (``bank``: that bank, found here when not given), else stacked."""
    a0 = attns[0]
    E, H, hd, d, P = a0.embed_dim, a0.num_heads, a0.head_dim, a0.fsq.dim, a0.code_dim
    G = len(attns)
    W = _stack([a.in_proj_weight for a in attns])                          # [G, 3E, E]
    Wq, Wk, Wv = W.split(E, 1)
    bank = shared_bank(attns) if bank is None else bank
    if bank is not None:                                                   # [G, d, hd], [G, d], [G, hd, d]
        Wd, bd, Wu = bank.down_weight, bank.down_bias, bank.up_weight
    else:
        Wd, bd = _stack([a.key_down.weight for a in attns]), _stack([a.key_down.bias for a in attns])
        Wu = _stack([a.key_up.weight for a in attns])
    _, _, shift, half_width = a0.fsq.constants(Wu.dtype)
    # (every product below consumes U and D in their own layout, so that their gradients, and the
    # parameters' through the stacks, come out contiguous: no copy per layer when they are stored)
    U = F.pad(Wu / half_width, (0, P - d))                                  # [G, hd, P]
    D = F.pad(Wd, (0, 0, 0, P - d))                                         # [G, P, hd]
    q_rows = torch.matmul(Wq.unflatten(1, (H, hd)).mT, U.unsqueeze(1)).mT  # [G, H, P, E]
    k_rows = torch.matmul(D.unsqueeze(1), Wk.unflatten(1, (H, hd)))        # [G, H, P, E]
    k_bias = F.pad(bd + shift, (0, P - d)).unsqueeze(-1)                    # [G, P, 1]
    if a0.in_proj_bias is not None:
        bq, bk, bv = _stack([a.in_proj_bias for a in attns]).split(E, 1)   # [G, E] each
        q_bias = torch.bmm(bq.unflatten(1, (H, hd)), U)                     # [G, H, P]
        k_bias = torch.baddbmm(k_bias, D, bk.unflatten(1, (H, hd)).mT).mT  # [G, H, P]
    else:
        q_bias, k_bias, bv = k_bias.new_zeros(G, H, P), k_bias.mT.expand(G, H, P), k_bias.new_zeros(G, E)
    # rows in blocks of P (no copy of the transposed query rows): [G, 2H + E/P, P, E] when P divides E
    blocks = E % P == 0
    weight = torch.cat([q_rows, k_rows, Wv.unflatten(1, (E // P, P))], 1).flatten(1, 2) if blocks else \
        torch.cat([q_rows.flatten(1, 2), k_rows.flatten(1, 2), Wv], 1)     # [G, 2HP + E, E]
    bias = torch.cat([q_bias, k_bias, bv.unflatten(1, (E // P, P))], 1).flatten(1) if blocks else \
        torch.cat([q_bias.flatten(1), k_bias.flatten(1), bv], 1)           # [G, 2HP + E]
    if dtype is not None and dtype != weight.dtype:
        weight, bias = weight.to(dtype), bias.to(dtype)
    return list(zip(weight.unbind(0), bias.unbind(0)))


class fold_keys:
    """Context manager, for one call with autograd: the folded in-projections
    (:func:`folded_projections`) of every layer in ``attns`` made at once, as stacked tensors (a
    fixed number of kernels for all layers, not a few per layer; under autocast one cast of the
    stacked result, not one per layer and use). Without autograd (cached per layer), under
    ``torch.compile`` (which fuses the folds itself), with fewer than two layers, or layers of
    different sizes, levels or dtypes, it does nothing."""

    def __init__(self, attns: Sequence["FSQMultiheadAttention"], like: Tensor) -> None:
        self.attns = [a for a in attns if a.quantize]
        self.like = like

    def __enter__(self) -> "fold_keys":
        attns = self.attns
        if (len(attns) < 2 or not torch.is_grad_enabled() or compiling()
                or len({(a.fsq.levels_list, a.embed_dim, a.num_heads, a.in_proj_bias is None,
                         a.in_proj_weight.dtype, a.in_proj_weight.device) for a in attns}) != 1):
            self.attns = []
            return self
        for a, proj in zip(attns, folded_projections(attns, compute_dtype(self.like))):
            a._call_proj = proj
        return self

    def __exit__(self, *exc) -> None:
        for a in self.attns:
            a._call_proj = None


def quantize_attention_keys(module: nn.Module, levels: Sequence[int], bank: bool = True) -> int:
    """In place: replace each ``self_attn`` ``nn.MultiheadAttention`` inside ``module`` (e.g. of
    ``nn.TransformerEncoderLayer`` / ``nn.TransformerDecoderLayer``) by
    :meth:`FSQMultiheadAttention.from_mha`. Cross-attention (``multihead_attn``) is left alone.
    ``nn.TransformerEncoder``'s nested-tensor setting stays (FSQ attention takes nested input;
    ``sparsify`` turns it off and back on). ``bank``: the new layers' key maps held as stacked
    parameters on ``module`` (:func:`~smdm_plugin.core.fsq_bank.bank_key_maps`, ``fsq_key_maps``:
    the same values; a state dict holds the bank's tensors, one of per-layer key maps loads).
    Returns the number replaced."""
    new = []
    for m in list(module.modules()):
        attn = getattr(m, "self_attn", None)
        if isinstance(attn, nn.MultiheadAttention):
            m.self_attn = FSQMultiheadAttention.from_mha(attn, levels)
            new.append(m.self_attn)
    if bank:
        bank_key_maps(module, new)
    return len(new)


def unquantize_attention_keys(module: nn.Module) -> int:
    """In place, the inverse of :func:`quantize_attention_keys`: each ``FSQMultiheadAttention``
    ``self_attn`` becomes an ``nn.MultiheadAttention`` with its current weights
    (:meth:`FSQMultiheadAttention.to_mha`), and the key-map banks go. Returns the number replaced."""
    count = 0
    for m in list(module.modules()):
        attn = getattr(m, "self_attn", None)
        if isinstance(attn, FSQMultiheadAttention):
            m.self_attn = attn.to_mha()
            count += 1
    remove_banks(module)
    return count
