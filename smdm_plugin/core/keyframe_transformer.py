"""Keyframe-only transformer: run an existing ``nn.TransformerEncoder``/``Decoder`` on keyframe
tokens only and interpolate its output back to every frame.

The wrapper keeps the wrapped module's children (``layers``, ``norm``) under the same names, so
state-dict keys do not change (``seqTransEncoder.layers.0...``). The keyframe mask is handed in
through :meth:`KeyframeTransformer.set_keyframes` right before the forward call (the adapters do this
from a forward pre-hook of the whole model); without one the wrapped module runs dense.
"""
from __future__ import annotations

from typing import Optional

import torch
import torch.nn as nn

from .attention_backends import get_backend, lerp_rows, supports_packed, varlen_backend, varlen_packed
from .interpolation import interpolate_keyframes, neighbour_keyframes


class KeyframeTransformer(nn.Module):
    """Wraps ``inner`` (an ``nn.TransformerEncoder`` or ``nn.TransformerDecoder``).

    Args:
        inner: the module to wrap; its layers and weights are used as they are.
        n_lead: unused, kept for clarity; the tokens before the frames that always stay (MDM
            trans_enc: the timestep/text token) are inferred as ``S - mask.shape[1]``.
        interpolate: fill non-keyframe outputs by linear interpolation (else they are zero).
        backend: ``auto`` | ``compact`` | ``varlen`` | ``masked`` (see ``attention_backends``).
    """

    def __init__(self, inner: nn.Module, n_lead: int = 0, interpolate: bool = True,
                 backend: str = "auto") -> None:
        super().__init__()
        if isinstance(inner, nn.TransformerEncoder):
            self.kind = "encoder"
        elif isinstance(inner, nn.TransformerDecoder):
            self.kind = "decoder"
        else:
            raise TypeError("KeyframeTransformer: inner must be nn.TransformerEncoder or "
                            f"nn.TransformerDecoder, got {type(inner).__name__}")
        object.__setattr__(self, "inner", inner)  # not registered: its children are, below
        for name, child in inner.named_children():
            self.add_module(name, child)
        first = inner.layers[0]
        self.batch_first = bool(getattr(first.self_attn, "batch_first", False))
        self.n_lead = int(n_lead)
        self.interpolate = interpolate
        self.backend = backend
        self._keyframes: Optional[torch.Tensor] = None

    def extra_repr(self) -> str:
        return f"kind={self.kind}, n_lead={self.n_lead}, backend={self.backend!r}"

    # ------------------------------------------------------------------ mask hand-over
    def set_keyframes(self, mask: Optional[torch.Tensor]) -> None:
        """``mask`` bool ``[B, N]`` over the frame tokens (after the ``n_lead`` tokens), or None."""
        self._keyframes = mask

    @property
    def keyframes(self) -> Optional[torch.Tensor]:
        return self._keyframes

    # ------------------------------------------------------------------ forward
    def forward(self, *args, **kwargs) -> torch.Tensor:
        """Same signature as the wrapped ``nn.TransformerEncoder`` / ``nn.TransformerDecoder``."""
        if self._keyframes is None:
            return self.inner(*args, **kwargs)
        if self.kind == "encoder":
            return self._forward_encoder(*args, **kwargs)
        return self._forward_decoder(*args, **kwargs)

    def _forward_encoder(self, src: torch.Tensor, mask: Optional[torch.Tensor] = None,
                         src_key_padding_mask: Optional[torch.Tensor] = None,
                         is_causal: Optional[bool] = None) -> torch.Tensor:
        if mask is not None or is_causal:
            raise NotImplementedError("KeyframeTransformer: attention masks (mask/is_causal) are not "
                                      "supported in sparse mode; only key padding masks")
        x = src.transpose(0, 1) if self.batch_first else src  # [S, B, d]
        keep = self._keep(x, src_key_padding_mask)
        fn = get_backend(self.backend, x.device, self.training)
        if fn is varlen_backend and self._packable(keep):
            out = self._packed_fill(*varlen_packed(self.inner, x, keep), keep)
        else:
            out = self._fill(fn(self.inner, x, keep), keep)
        return out.transpose(0, 1) if self.batch_first else out

    def _forward_decoder(self, tgt: torch.Tensor, memory: torch.Tensor,
                         tgt_mask: Optional[torch.Tensor] = None, memory_mask: Optional[torch.Tensor] = None,
                         tgt_key_padding_mask: Optional[torch.Tensor] = None,
                         memory_key_padding_mask: Optional[torch.Tensor] = None,
                         tgt_is_causal: Optional[bool] = None, memory_is_causal: bool = False) -> torch.Tensor:
        if tgt_mask is not None or memory_mask is not None or tgt_is_causal or memory_is_causal:
            raise NotImplementedError("KeyframeTransformer: attention masks (tgt_mask/memory_mask/causal)"
                                      " are not supported in sparse mode; only key padding masks")
        x = tgt.transpose(0, 1) if self.batch_first else tgt
        mem = memory.transpose(0, 1) if self.batch_first else memory
        keep = self._keep(x, tgt_key_padding_mask)
        fn = get_backend(self.backend, x.device, self.training)
        if fn is varlen_backend and self._packable(keep):
            h, packing = varlen_packed(self.inner, x, keep, memory=mem,
                                       memory_key_padding_mask=memory_key_padding_mask)
            out = self._packed_fill(h, packing, keep)
        else:
            out = self._fill(fn(self.inner, x, keep, memory=mem, memory_key_padding_mask=memory_key_padding_mask),
                             keep)
        return out.transpose(0, 1) if self.batch_first else out

    # ------------------------------------------------------------------ helpers
    def _keep(self, x: torch.Tensor, key_padding_mask: Optional[torch.Tensor]) -> torch.Tensor:
        """bool ``[B, S]``: lead tokens + keyframes, minus padded tokens."""
        S, B, _ = x.shape
        kf = self._keyframes.to(device=x.device, dtype=torch.bool)
        if kf.dim() != 2 or kf.shape[0] != B or kf.shape[1] > S:
            raise ValueError(f"KeyframeTransformer: keyframe mask must be [B, N] with B={B} and "
                             f"N <= S={S} (sequence length), got {tuple(kf.shape)}")
        self.n_lead = S - kf.shape[1]
        keep = torch.cat([kf.new_ones(B, self.n_lead), kf], dim=1) if self.n_lead else kf
        if key_padding_mask is not None:
            keep = keep & ~key_padding_mask.to(torch.bool)
        return keep

    def _packable(self, keep: torch.Tensor) -> bool:
        """Interpolate straight from the packed rows (needs every lead token kept)."""
        return (self.interpolate and supports_packed(self.inner)
                and (self.n_lead == 0 or bool(keep[:, :self.n_lead].all())))

    def _packed_fill(self, h: torch.Tensor, packing, keep: torch.Tensor) -> torch.Tensor:
        """Same result as scattering the packed rows ``h [T, d]`` back to ``[S, B, d]`` and
        :meth:`_fill`, but read straight from the packed rows (no zero-filled ``[S, B, d]``
        intermediate, no concatenation): every output token is ``lerp(h[prev], h[next], w)``; lead
        and kept tokens have ``prev = next`` = their own row and ``w = 0``."""
        B, S = keep.shape
        lead = self.n_lead
        frames = keep[:, lead:]
        if not bool(frames.any(dim=1).all()):
            raise ValueError("interpolate_keyframes: every row of mask needs at least one keyframe")
        rowmap = torch.zeros(B, S, dtype=torch.long, device=keep.device)
        rowmap[packing.seg, packing.src] = torch.arange(packing.T, device=keep.device)
        prev, nxt, w = neighbour_keyframes(frames, h.dtype)
        fr = rowmap[:, lead:]
        prev_r, next_r = fr.gather(1, prev), fr.gather(1, nxt)
        if lead:
            prev_r = torch.cat([rowmap[:, :lead], prev_r], 1)
            next_r = torch.cat([rowmap[:, :lead], next_r], 1)
            w = torch.cat([w.new_zeros(B, lead), w], 1)
        d = h.shape[-1]
        out = lerp_rows(h, prev_r.t().reshape(-1), next_r.t().reshape(-1), w.t().reshape(-1, 1))
        return out.view(S, B, d)

    def _fill(self, out: torch.Tensor, keep: torch.Tensor) -> torch.Tensor:
        """Interpolate frame tokens (rows ``n_lead:``) from the kept ones. ``out [S, B, d]``."""
        if not self.interpolate:
            return out * keep.t().unsqueeze(-1).to(out.dtype)
        lead, frames = out[: self.n_lead], out[self.n_lead:]
        filled = interpolate_keyframes(frames.transpose(0, 1), keep[:, self.n_lead:]).transpose(0, 1)
        return torch.cat([lead, filled], dim=0) if self.n_lead else filled
