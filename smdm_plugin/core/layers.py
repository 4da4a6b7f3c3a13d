"""PyTorch's stock transformer layers run as functions on the kept tokens (the compact backend)."""
from __future__ import annotations

import math
from typing import Callable, Dict, List, Optional, Sequence, Tuple

import torch
import torch.nn as nn
import torch.nn.functional as F
from torch import Tensor

from . import consts
from .attention import attend_single_key, compute_dtype, heads as _heads, layout_copies
from .checks import compiling
from .fsq import FSQMultiheadAttention, folded_projections
from .fsq_bank import key_map_tensors, shared_bank
from .kernels.fsq_code import code_functions
from .products import ProductStore, Remade
from .structure import structure_version

__all__ = ["StockStack", "stock_stack"]

_ENC, _DEC = nn.TransformerEncoderLayer, nn.TransformerDecoderLayer
_HOOK_DICTS = ("_forward_hooks", "_forward_pre_hooks", "_backward_hooks", "_backward_pre_hooks")

def _merge(o: Tensor) -> Tensor:
    """``[B, H, S, e]`` -> ``[S·B, H·e]`` (one copy, as ``nn.MultiheadAttention``)."""
    B, H, S, e = o.shape
    return o.permute(2, 0, 1, 3).reshape(S * B, H * e)


#: per call under autocast, the layers' matmul weights and biases in autocast's dtype, by the
#: parameter's ``id`` (or None: the parameters themselves; :meth:`StockStack._casts`)
Casts = Optional[Dict[int, Tensor]]


def _linear(m: nn.Module, casts: Casts = None, weight: str = "weight", bias: str = "bias"
            ) -> Tuple[Tensor, Optional[Tensor]]:
    """``m``'s ``weight`` and ``bias`` parameters (named so), read from the module at each call (a move
    or a reload is seen), from ``casts`` when given."""
    p = m._parameters
    w, b = p[weight], p[bias]
    if casts is None:
        return w, b
    return casts[id(w)], None if b is None else casts[id(b)]


#: how a stack's FSQ layers make their codes in one run (:func:`~smdm_plugin.core.kernels.fsq_code.code_functions`):
#: ``(with autograd, without)``
Codes = Tuple[Callable[..., Tensor], Callable[..., Tensor]]


class _Attention:
    """One attention module, called as a function (its tensors read from the module at each call:
    a move or a reload is seen)."""

    def __init__(self, m: nn.Module) -> None:
        self.module, self.out = m, m.out_proj
        self.heads = m.num_heads
        self.folded = isinstance(m, FSQMultiheadAttention) and m.quantize
        if self.folded:
            self.code_dim, self.scale = m.code_dim, 1.0 / math.sqrt(m.head_dim)

    def self_attention(self, x: Tensor, S: int, bias: Optional[Tensor], p: float, proj: Optional[tuple],
                       copy: bool, casts: Casts, codes: Optional[Codes]) -> Tensor:
        """Self-attention of the rows ``x [S·B, E]`` of ``S`` tokens (key mask ``bias [B, 1, 1, S]``
        or None, attention dropout ``p``; ``proj``: how an FSQ layer makes its codes,
        :meth:`StockStack._projections`; ``casts``: :meth:`StockStack._casts`; ``codes``: the
        run's :data:`Codes`): ``[S·B, E]``."""
        E = x.shape[1]
        H, m = self.heads, self.module
        scale = None
        if self.folded:                                        # FSQ keys (core/fsq.py)
            P = self.code_dim
            # one folded in-projection, its tokens split out before the heads (a gradient meets its
            # heads' in one copy, the split's, not one per head)
            qc, z, v = F.linear(x, proj[1], proj[2]).view(S, -1, 2 * H * P + E).split_with_sizes([H * P, H * P, E], -1)
            buffers = m._buffers
            code = codes[0] if z.requires_grad and torch.is_grad_enabled() else codes[1]
            k = code(z, buffers["_code_neg_offset"], buffers["_code_half_l"])
            q, k, v = _heads(qc, H, copy), _heads(k, H, copy), _heads(v, H, copy)
            scale = self.scale
        else:
            qkv = F.linear(x, *_linear(m, casts, "in_proj_weight", "in_proj_bias")).view(S, -1, 3 * E)
            q, k, v = qkv.chunk(3, dim=-1)
            q, k, v = _heads(q, H, copy), _heads(k, H, copy), _heads(v, H, copy)
        o = F.scaled_dot_product_attention(q, k, v, attn_mask=bias, dropout_p=p, scale=scale)
        return F.linear(_merge(o), *_linear(self.out, casts))

    def cross_attention(self, x: Tensor, S: int, memory: Tensor, bias: Optional[Tensor], p: float,
                        sample: Optional[Tensor], copy: bool, casts: Casts) -> Tensor:
        """Attention of the rows ``x [S·B, E]`` of ``S`` tokens to ``memory [M, B, E]`` (key mask
        ``bias [B, 1, 1, M]`` or None): ``[S·B, E]``. One key per sample (MDM trans_dec's condition
        token) needs no softmax (:func:`~smdm_plugin.core.attention.attend_single_key`; ``sample
        [S·B]``)."""
        if sample is not None:
            o = attend_single_key(self.module, memory[0], sample)
        else:
            E, H = x.shape[1], self.heads
            W, b = _linear(self.module, casts, "in_proj_weight", "in_proj_bias")
            q = _heads(F.linear(x, W[:E], None if b is None else b[:E]).view(S, -1, E), H, copy)
            k, v = F.linear(memory, W[E:], None if b is None else b[E:]).chunk(2, dim=-1)
            k, v = _heads(k, H, copy), _heads(v, H, copy)
            o = _merge(F.scaled_dot_product_attention(q, k, v, attn_mask=bias, dropout_p=p))
        return F.linear(o, *_linear(self.out, casts))


def _layer_norm(x: Tensor, m: nn.LayerNorm) -> Tensor:
    """``F.layer_norm`` by ``m``, without its Python wrapper (the same call)."""
    p = m._parameters
    return torch.layer_norm(x, m.normalized_shape, p["weight"], p["bias"], m.eps, torch.backends.cudnn.enabled)


class _Layer:
    """One stock layer, called as a function."""

    def __init__(self, layer: nn.Module) -> None:
        self.module = layer
        self.decoder = type(layer) is _DEC
        self.self_attn = _Attention(layer.self_attn)
        self.cross = _Attention(layer.multihead_attn) if self.decoder else None
        names = ("norm1", "norm2", "norm3") if self.decoder else ("norm1", "norm2")
        self.norms = [getattr(layer, n) for n in names]
        self.l1, self.l2 = layer.linear1, layer.linear2
        self.drops = [getattr(layer, n) for n in ("dropout", "dropout1", "dropout2", "dropout3") if hasattr(layer, n)]

    def matmul_parameters(self) -> List[Tensor]:
        """The parameters this layer reads as matmul weights and biases (what a sampling call may
        read in its compute dtype: :meth:`StockStack._casts`); not the norms' (autocast runs
        ``layer_norm`` in float32), not a folded in-projection's (made by the fold), not the
        single-key cross-attention's value projection (read by ``attend_single_key``)."""
        mods = [self.self_attn.out, self.l1, self.l2] + ([self.cross.out] if self.decoder else [])
        out = [t for m in mods for t in _linear(m)]
        attns = [] if self.self_attn.folded else [self.self_attn.module]
        attns += [self.cross.module] if self.decoder else []
        out += [a._parameters[n] for a in attns for n in ("in_proj_weight", "in_proj_bias")]
        return [t for t in out if t is not None]

    def forward(self, x: Tensor, S: int, bias: Optional[Tensor], proj: Optional[tuple], training: bool,
                copy: bool, memory: Optional[Tensor] = None, memory_bias: Optional[Tensor] = None,
                sample: Optional[Tensor] = None, casts: Casts = None, codes: Optional[Codes] = None) -> Tensor:
        """The layer's ``forward`` (encoder or decoder, either ``norm_first``) on the rows ``x [S·B,
        d]`` of ``S`` tokens, sequence-first (``casts``: :meth:`StockStack._casts`; ``codes``: the
        run's :data:`Codes`). Written out block by block (no closure or helper per block: a step
        of MDM's eight layers pays Python per call); in eval no dropout call at all."""
        d, norms, first = self.drops, self.norms, self.module.norm_first
        # self-attention block
        h = _layer_norm(x, norms[0]) if first else x
        h = self.self_attn.self_attention(h, S, bias, self.self_attn.module.dropout if training else 0.0, proj,
                                          copy, casts, codes)
        if training and d[1].p:
            h = F.dropout(h, d[1].p, True)
        x = x + h if first else _layer_norm(x + h, norms[0])
        if self.decoder:                                      # cross-attention block
            h = _layer_norm(x, norms[1]) if first else x
            h = self.cross.cross_attention(h, S, memory, memory_bias, self.cross.module.dropout if training else 0.0,
                                           sample, copy, casts)
            if training and d[2].p:
                h = F.dropout(h, d[2].p, True)
            x = x + h if first else _layer_norm(x + h, norms[1])
        # feed-forward block
        h = _layer_norm(x, norms[-1]) if first else x
        h = self.module.activation(F.linear(h, *_linear(self.l1, casts)))
        if training and d[0].p:
            h = F.dropout(h, d[0].p, True)
        h = F.linear(h, *_linear(self.l2, casts))
        if training and d[-1].p:
            h = F.dropout(h, d[-1].p, True)
        return x + h if first else _layer_norm(x + h, norms[-1])


def _is_stock_mha(m: nn.Module) -> bool:
    return type(m) is nn.MultiheadAttention and m._qkv_same_embed_dim and m.bias_k is None \
        and not m.add_zero_attn and m.embed_dim % m.num_heads == 0


def _is_stock_attention(m: nn.Module) -> bool:
    return _is_stock_mha(m) or type(m) is FSQMultiheadAttention


def _stock_layer(layer: nn.Module) -> bool:
    kind = type(layer)
    if kind is _ENC:
        ok = _is_stock_attention(layer.self_attn)
    elif kind is _DEC:
        ok = _is_stock_attention(layer.self_attn) and _is_stock_mha(layer.multihead_attn)
    else:
        return False
    return ok and all(type(m) in (nn.Linear, nn.LayerNorm, nn.Dropout) for name, m in layer.named_children()
                      if name.startswith(("linear", "norm", "dropout")))


class StockStack(Remade):
    """The layers of a wrapped ``nn.TransformerEncoder`` / ``Decoder`` that run as functions
    (:func:`stock_stack`); :meth:`run` is the stack's forward on sequence-first tokens."""

    def __init__(self, inner: nn.Module) -> None:
        self.inner = inner
        self.version = structure_version()
        self.decoder = isinstance(inner, nn.TransformerDecoder)
        self.norm: Optional[nn.Module] = inner.norm
        self.layers = [_Layer(layer) for layer in inner.layers]
        self._folded = [a.self_attn.module for a in self.layers if a.self_attn.folded]
        self._bank = shared_bank(self._folded)            # their key maps as stacked parameters, or None
        # what the folds are made of, each tensor once, for the sampling cache's key (a parameter
        # replaced is a registration: rebuilt; a move or cast replaces the FSQ constants' buffers
        # unregistered, but changes the parameters' storage too: the key changes)
        self._fold_inputs = list({id(t): t for m in self._folded for t in _fold_tensors(m) if t is not None}.values())
        self._fsq = [m for m in inner.modules() if isinstance(m, FSQMultiheadAttention)]
        self._quantize = tuple(m.quantize for m in self._fsq)
        modules = list(inner.modules())
        # hooks would not run on the functional path; FSQ attention's own no-op pre-hook is known
        fsq = {id(m) for m in self._fsq}
        self._hooks = [getattr(m, n) for m in modules for n in _HOOK_DICTS
                       if not (n == "_forward_pre_hooks" and id(m) in fsq)]
        self._fsq_pre = [m._forward_pre_hooks for m in self._fsq]
        # without autograd, outside tracing: the folds and the weights' casts kept while their
        # parameters are unchanged (:class:`~smdm_plugin.core.products.ProductStore`); and the last
        # per-layer view of each (remade only when the store holds other tensors)
        self._fold_store, self._cast_store = ProductStore(), ProductStore()
        self._fold_view: tuple = (None, None)
        self._cast_view: tuple = (None, None)
        self._matmul = [t for layer in self.layers for t in layer.matmul_parameters()]

    def current(self) -> bool:
        """No module, parameter or buffer was registered anywhere since the stack was built (a
        replaced layer or submodule is a registration), and every FSQ attention still quantises as
        it did (``quantize`` is a plain attribute)."""
        version = structure_version()
        return version is not None and self.version == version and self._quantize == tuple(m.quantize for m in self._fsq)

    def usable(self) -> bool:
        """No hook on any module of the stack (it would not run here), no global module hooks."""
        return not (any(self._hooks) or (self._fsq_pre and max(map(len, self._fsq_pre)) > 1)
                    or _global_hooks())

    def _projections(self, dtype: torch.dtype) -> List[Optional[tuple]]:
        """Per layer, ``("fold", weight, bias)``: the folded in-projection of its FSQ self-attention
        in ``dtype`` (:func:`~smdm_plugin.core.fsq.folded_projections`: every layer's at once; one
        matmul per layer), None for the other layers. Without autograd and outside tracing kept
        while the parameters are the same tensors at the same versions (a sampling loop folds once).
        (Applying the key maps to the activations instead — ``q_h U^T``, ``k_h D^T + c`` per layer —
        is the same maths but costs more host time in the backward: measured, not used.)"""
        if not self._folded:
            return [None] * len(self.layers)
        if torch.is_grad_enabled() or compiling():
            folds = iter(folded_projections(self._folded, dtype, self._bank))
            return [("fold",) + next(folds) if a.self_attn.folded else None for a in self.layers]
        held = self._fold_store.get(dtype, self._fold_inputs, lambda: [
            t for fold in folded_projections(self._folded, dtype, self._bank) for t in fold])
        if self._fold_view[0] is not held:
            folds = iter(zip(held[0::2], held[1::2]))
            self._fold_view = (held, [("fold",) + next(folds) if a.self_attn.folded else None
                                      for a in self.layers])
        return self._fold_view[1]

    def _casts(self, x: Tensor) -> Casts:
        """The layers' matmul weights and biases (:meth:`_Layer.matmul_parameters`) in autocast's
        dtype for ``x``'s device, by parameter ``id``, the values autocast would make (it leaves
        float64 alone). Without autograd cast once, not at every call (autocast casts each weight
        at each use, its cache lasting one ``autocast`` block: ~6 casts per layer and call), kept
        while the parameters are the same tensors at the same versions (an optimizer step, a move
        or a reload makes new copies); with autograd :meth:`_stacked_casts` (traced too: a compiled
        training step casts each role once, not each weight). None while tracing a call without
        autograd (the stack does not run there), without autocast, or when the parameters already
        are in its dtype."""
        params = self._matmul
        if (compiling() and not torch.is_grad_enabled()) or not params or x.device.type == "meta" \
                or not torch.is_autocast_enabled(x.device.type):
            return None
        dtype = torch.get_autocast_dtype(x.device.type)
        if all(t.dtype in (dtype, torch.float64) for t in params):
            return None
        if torch.is_grad_enabled():
            return self._stacked_casts(dtype)
        held = self._cast_store.get(dtype, params, lambda: [t if t.dtype == torch.float64 else t.detach().to(dtype)
                                                            for t in params])  # (autocast leaves float64 alone)
        if self._cast_view[0] is not held:
            self._cast_view = (held, dict(zip(map(id, params), held)))
        return self._cast_view[1]

    def _stacked_casts(self, dtype: torch.dtype) -> Casts:
        """With autograd: each matmul parameter's cast as one stack, cast and unbind per role over
        the layers (3 ops each way for all layers instead of one cast each way per layer), when
        every layer has the same parameters of the same shapes and dtypes; else None."""
        per = len(self._matmul) // len(self.layers)
        groups = [self._matmul[i::per] for i in range(per)]
        if per * len(self.layers) != len(self._matmul) or len(self.layers) < 2 or any(
                len({(t.shape, t.dtype, t.device) for t in g}) != 1 or g[0].dtype == torch.float64 for g in groups):
            return None
        return {id(t): c for g in groups for t, c in zip(g, torch.stack(g).to(dtype).unbind(0))}

    def run(self, x: Tensor, bias: Optional[Tensor], memory: Optional[Tensor] = None,
            memory_bias: Optional[Tensor] = None) -> Tensor:
        """``x [S, B, d]`` sequence-first through every layer (and the stack's norm): :meth:`run_rows`
        on its rows, ``[S, B, d]``."""
        S, B, d = x.shape
        return self.run_rows(x.reshape(S * B, d), S, bias, memory, memory_bias).view(S, B, d)

    def run_rows(self, x: Tensor, S: int, bias: Optional[Tensor], memory: Optional[Tensor] = None,
                 memory_bias: Optional[Tensor] = None) -> Tensor:
        """The rows ``x [S·B, d]`` of ``S`` tokens, sequence-first, through every layer (and the
        stack's norm), ``[S·B, d]`` (the layers' linear maps on rows as they are: no reshape per
        map and gradient); ``bias [B, 1, 1, S]`` additive key mask or None; decoders: ``memory [M,
        B, d]``, ``memory_bias [B, 1, 1, M]`` or None."""
        training = self.layers[0].module.training     # (the wrapper keeps the stack unregistered)
        dtype = compute_dtype(x)
        projections = self._projections(dtype)
        sample = None
        if self.decoder and memory.shape[0] == 1 and memory_bias is None:   # one key per sample
            sample = consts.arange(x.shape[0] // S, x.device).repeat(S)   # [S·B]: each row's sample
        copy = layout_copies()                                # views unless switched on (use_layout_copies)
        casts = self._casts(x)
        codes = code_functions(x) if self._folded else None
        for layer, proj in zip(self.layers, projections):
            x = layer.forward(x, S, bias, proj, training, copy, memory, memory_bias, sample, casts, codes)
        return x if self.norm is None else self.norm(x)


def _fold_tensors(m: FSQMultiheadAttention) -> Tuple[Tensor, ...]:
    """What an FSQ layer's folded in-projection is made of (read without module attribute lookups;
    a banked layer's key maps: its bank's tensors)."""
    p, fsq = m._parameters, m._modules["fsq"]._buffers
    return (p["in_proj_weight"], p["in_proj_bias"], *key_map_tensors(m)[:3], fsq["_shift"], fsq["_half_width"])


def _global_hooks() -> bool:
    from torch.nn.modules import module as m

    return bool(m._global_forward_hooks or m._global_forward_pre_hooks or m._global_backward_hooks
                or getattr(m, "_global_backward_pre_hooks", None))


def stock_stack(inner: nn.Module) -> Optional[StockStack]:
    """The :class:`StockStack` of ``inner`` when every layer is a stock layer and nothing hooks
    into its modules, else None (run the modules). Built once per stack (rebuilt after any module
    registration, so a replaced submodule is seen). While ``torch.compile`` traces a call with
    autograd, built in the trace (no cache for the graph to guard on): its layers then read every
    FSQ fold of the stack made at once (batched matmuls), not one fold per layer; a traced call
    without autograd runs the modules (they read the folds a compiled call keeps:
    :mod:`~smdm_plugin.core.products`)."""
    if compiling():
        if not torch.is_grad_enabled() or not all(_stock_layer(layer) for layer in inner.layers):
            return None
        stack = StockStack(inner)
        return stack if stack.usable() else None
    stack = inner.__dict__.get("_smdm_stock")
    if stack is not None and stack.current():
        return stack if stack.usable() else None
    if not all(_stock_layer(layer) for layer in inner.layers):
        return None
    stack = StockStack(inner)
    inner.__dict__["_smdm_stock"] = stack
    return stack if stack.usable() else None
