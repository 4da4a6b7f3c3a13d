"""Keyframe-only transformer: run an existing ``nn.TransformerEncoder``/``Decoder`` on keyframe
tokens only and interpolate its output back to every frame.

The wrapper keeps the wrapped module's children (``layers``, ``norm``) under the same names, so
state-dict keys do not change (``seqTransEncoder.layers.0...``). The keyframes of a call arrive as a
:class:`~smdm_plugin.core.plan.KeyframePlan` through :meth:`KeyframeTransformer.set_plan` right
before the forward call (the adapters do this from a forward pre-hook of the whole model); without
one the wrapped module runs dense, exactly as before.
"""
from __future__ import annotations

from typing import Optional

import torch
import torch.nn as nn

from .attention_backends import get_backend
from .fill import fill_frames
from .checks import host_checkable
from .plan import KeyframePlan


class KeyframeTransformer(nn.Module):
    """Wraps ``inner`` (an ``nn.TransformerEncoder`` or ``nn.TransformerDecoder``).

    Args:
        inner: the module to wrap; its layers and weights are used as they are.
        interpolate: fill non-keyframe outputs by linear interpolation (else they are zero).
        backend: ``auto`` | ``compact`` | ``varlen`` | ``masked`` (see ``attention_backends``).

    Tokens before the frames that always stay (MDM trans_enc: the timestep/text token) are
    ``S - plan.frames`` for a sequence of ``S`` tokens.
    """

    def __init__(self, inner: nn.Module, interpolate: bool = True, backend: str = "auto") -> None:
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
        self.batch_first = bool(getattr(inner.layers[0].self_attn, "batch_first", False))
        self.interpolate = interpolate
        self.backend = backend
        self._plan: Optional[KeyframePlan] = None

    def extra_repr(self) -> str:
        return f"kind={self.kind}, backend={self.backend!r}, interpolate={self.interpolate}"

    # ------------------------------------------------------------------ plan hand-over
    def set_plan(self, plan: Optional[KeyframePlan]) -> None:
        """The keyframes of the next call(s), or None to run dense."""
        self._plan = plan

    def set_keyframes(self, mask: Optional[torch.Tensor], capacity: Optional[int] = None) -> None:
        """Convenience: a plan from bool ``mask [B, N]`` over the frame tokens (after the lead
        tokens). ``capacity`` None: ``N`` slots (always enough; pass the real bound for speed)."""
        self._plan = None if mask is None else KeyframePlan.build(mask, capacity)

    @property
    def plan(self) -> Optional[KeyframePlan]:
        return self._plan

    @property
    def keyframes(self) -> Optional[torch.Tensor]:
        return None if self._plan is None else self._plan.mask

    # ------------------------------------------------------------------ forward
    def forward(self, *args, **kwargs) -> torch.Tensor:
        """Same signature as the wrapped ``nn.TransformerEncoder`` / ``nn.TransformerDecoder``."""
        if self._plan is None:
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
        return self._run(src, src_key_padding_mask)

    def _forward_decoder(self, tgt: torch.Tensor, memory: torch.Tensor,
                         tgt_mask: Optional[torch.Tensor] = None, memory_mask: Optional[torch.Tensor] = None,
                         tgt_key_padding_mask: Optional[torch.Tensor] = None,
                         memory_key_padding_mask: Optional[torch.Tensor] = None,
                         tgt_is_causal: Optional[bool] = None, memory_is_causal: bool = False) -> torch.Tensor:
        if tgt_mask is not None or memory_mask is not None or tgt_is_causal or memory_is_causal:
            raise NotImplementedError("KeyframeTransformer: attention masks (tgt_mask/memory_mask/causal)"
                                      " are not supported in sparse mode; only key padding masks")
        mem = memory.transpose(0, 1) if self.batch_first else memory
        return self._run(tgt, tgt_key_padding_mask, mem, memory_key_padding_mask)

    def _run(self, seq: torch.Tensor, key_padding_mask: Optional[torch.Tensor],
             memory: Optional[torch.Tensor] = None, memory_key_padding_mask: Optional[torch.Tensor] = None
             ) -> torch.Tensor:
        x = seq.transpose(0, 1) if self.batch_first else seq  # [S, B, d]
        plan = self._plan
        S, B, _ = x.shape
        if plan.batch != B or plan.frames > S:
            raise ValueError(f"KeyframeTransformer: the keyframe plan is for [B, N]=[{plan.batch}, "
                             f"{plan.frames}], the sequence has B={B}, S={S} tokens")
        if B == 0:  # an empty batch: the empty output (a Python-level shape check, no sync)
            return seq.clone()
        lead = S - plan.frames
        # padding of the frames is the plan's business (keyframes are valid frames); the caller's
        # padding of the lead tokens is honoured
        lead_padding = None
        if key_padding_mask is not None and lead:
            lead_padding = key_padding_mask[:, :lead].to(torch.bool)
            if host_checkable(lead_padding) and not bool(lead_padding.any()):
                lead_padding = None
        fn = get_backend(self.backend, x.device, self.inner, lead_padding is not None)
        h, rows = fn(self.inner, x, plan, lead, memory, memory_key_padding_mask, lead_padding)
        out = fill_frames(h, rows, plan, lead, self.interpolate)
        return out.transpose(0, 1) if self.batch_first else out
